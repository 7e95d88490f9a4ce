"""The compiled RK4 integrator of the geodetic state (numba): the same guidance laws and
geodetic rates as the numpy reference (kinematics.py), vehicle by vehicle; absent without numba.

A law hands the integrator its code and one parameter row per vehicle (``_kernel_args``)."""
from __future__ import annotations

import math

import numpy as np

try:  # compiled integration loop; the numpy path (kinematics.py) is the reference
    import numba as nb
except ImportError:  # pragma: no cover
    nb = None

# Law codes and the per-vehicle parameter row of the compiled integrator (_integrate_nb).
_LAW_SINUSOID, _LAW_LEGS, _LAW_HOLD, _LAW_WAYPOINTS, _LAW_RACETRACK = 0, 1, 2, 3, 4
_N_PARAMS = 11

ready = _integrate_nb = _integrate_track_nb = None  # without numba

if nb is not None:
    from filters.nbdispatch import declare, ready, ro, rw  # noqa: F401  (ready: called by kinematics and swarm)

    _TWO_PI = 2.0 * math.pi

    @nb.njit(cache=True, nogil=True)
    def _wrap_nb(a):
        return a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI)

    @nb.njit(cache=True, nogil=True)
    def _offset_nb(lat, lon, h, glat, glon, a, e2):
        w2 = 1.0 - e2 * math.sin(lat) ** 2
        n = a / math.sqrt(w2)
        m = n * (1.0 - e2) / w2
        return _wrap_nb(glon - lon) * (n + h) * math.cos(lat), (glat - lat) * (m + h)

    @nb.njit(cache=True, nogil=True)
    def _rates_nb(law, p, seg, tr, g, t, lat, lon, h, psi, a, e2):
        """The same law and geodetic rates as SinusoidalLaw/LegsAndTurns/Hold/WaypointMission/Racetrack
        .commands + geodetic_rates, for one vehicle (p its parameter row, seg the schedule
        interval of the step, g its waypoint)."""
        if law == 0:
            speed = p[0] + p[1] * math.sin(p[2] * t + p[3])
            climb = p[8] * math.cos(p[9] * t + p[10])
            rate = p[5] * p[6] * math.cos(p[6] * t + p[7])
        elif law == 1:
            speed = p[0]
            climb = 0.0
            rate = tr[seg]
        elif law == 2:
            speed = 0.0
            climb = 0.0
            rate = 0.0
        elif law == 4:  # Racetrack: p = speed, max rate, radius, turn gain, radial gain, centre lat, lon, axis, L
            d_e, d_n = _offset_nb(lat, lon, h, p[5], p[6], a, e2)
            sa, ca = math.sin(p[7]), math.cos(p[7])
            s = -(d_e * sa + d_n * ca)
            c = -(d_e * ca - d_n * sa)
            r = p[2]
            if s > p[8] or s < -p[8]:
                end = p[8] if s > 0 else -p[8]
                g_e, g_n = d_e + end * sa, d_n + end * ca
                ref = math.atan2(g_e, g_n) - 0.5 * math.pi + math.atan(p[4] * (math.hypot(g_e, g_n) - r) / r)
                ff = p[0] / r
            elif c < 0:
                ref = p[7] - math.atan(p[4] * (c + r) / r)
                ff = 0.0
            else:
                ref = p[7] + math.pi - math.atan(p[4] * (r - c) / r)
                ff = 0.0
            rate = min(max(ff + p[3] * _wrap_nb(ref - psi), -p[1]), p[1])
            climb = 0.0
            speed = p[0]
        else:
            d_e, d_n = _offset_nb(lat, lon, h, g[0], g[1], a, e2)
            rate = min(max(p[4] * _wrap_nb(math.atan2(d_e, d_n) - psi), -p[1]), p[1])
            climb = min(max(p[5] * (g[2] - h), -p[2]), p[2])
            speed = p[0]
        v_h = math.sqrt(max(speed * speed - climb * climb, 0.0))
        w2 = 1.0 - e2 * math.sin(lat) ** 2
        n = a / math.sqrt(w2)
        m = n * (1.0 - e2) / w2
        return (v_h * math.cos(psi) / (m + h), v_h * math.sin(psi) / ((n + h) * math.cos(lat)), climb, rate)

    @nb.njit(cache=True, nogil=True)
    def _rk4_steps_nb(law, p, tri, wpi, cnti, sw, ts, j0, j1, lat, lon, h, psi, k_wp, a, e2):
        """RK4 of one vehicle over the step boundaries ts[j0..j1]; returns the new state."""
        for k in range(j0, j1):
            ta = ts[k]
            tb = ts[k + 1]
            hh = tb - ta
            seg = np.searchsorted(sw, 0.5 * (ta + tb), side="right")
            g = wpi[min(k_wp, cnti - 1)]
            a1, b1, c1, d1 = _rates_nb(law, p, seg, tri, g, ta, lat, lon, h, psi, a, e2)
            a2, b2, c2, d2 = _rates_nb(law, p, seg, tri, g, ta + 0.5 * hh, lat + 0.5 * hh * a1,
                                       lon + 0.5 * hh * b1, h + 0.5 * hh * c1, psi + 0.5 * hh * d1, a, e2)
            a3, b3, c3, d3 = _rates_nb(law, p, seg, tri, g, ta + 0.5 * hh, lat + 0.5 * hh * a2,
                                       lon + 0.5 * hh * b2, h + 0.5 * hh * c2, psi + 0.5 * hh * d2, a, e2)
            a4, b4, c4, d4 = _rates_nb(law, p, seg, tri, g, tb, lat + hh * a3, lon + hh * b3, h + hh * c3,
                                       psi + hh * d3, a, e2)
            lat = lat + (hh / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            lon = _wrap_nb(lon + (hh / 6.0) * (b1 + 2.0 * b2 + 2.0 * b3 + b4))
            h = h + (hh / 6.0) * (c1 + 2.0 * c2 + 2.0 * c3 + c4)
            psi = psi + (hh / 6.0) * (d1 + 2.0 * d2 + 2.0 * d3 + d4)
            psi = psi - _TWO_PI * math.floor(psi / _TWO_PI)
            if law == 3:
                g = wpi[min(k_wp, cnti - 1)]
                d_e, d_n = _offset_nb(lat, lon, h, g[0], g[1], a, e2)
                if math.hypot(d_e, d_n) < p[3]:
                    k_wp = min(k_wp + 1, cnti)
        return lat, lon, h, psi, k_wp

    # one compiled version each (filters/nbdispatch.py): the guidance's arrays may be read-only
    @declare(nb.int64, rw(2), rw(1, nb.int64), ro(2), ro(1), ro(2), ro(3), ro(1, dtype=nb.int64), ro(1), nb.float64,
             nb.float64)
    @nb.njit(cache=True, nogil=True)
    def _integrate_nb(law, y, idx, params, sw, tr, wp, cnt, ts, a, e2):
        """RK4 over the step boundaries ts in place on y (N, 4) and idx (N,), one vehicle at a time."""
        for i in range(y.shape[0]):
            tri = tr[i] if law == 1 else tr[0]
            lat, lon, h, psi, k_wp = _rk4_steps_nb(law, params[i], tri, wp[i], cnt[i], sw, ts, np.int64(0), ts.size - 1,
                                                   y[i, 0], y[i, 1], y[i, 2], y[i, 3], idx[i], a, e2)
            y[i, 0], y[i, 1], y[i, 2], y[i, 3] = lat, lon, h, psi
            idx[i] = k_wp

    @declare(nb.int64, rw(2), rw(1, nb.int64), ro(2), ro(1), ro(2), ro(3), ro(1, dtype=nb.int64), ro(1),
             ro(1, dtype=nb.int64), rw(3), rw(2, nb.int64), nb.float64, nb.float64)
    @nb.njit(cache=True, nogil=True)
    def _integrate_track_nb(law, y, idx, params, sw, tr, wp, cnt, ts, ends, ys, idxs, a, e2):
        """As _integrate_nb over ts, recording the state at the boundaries ts[ends[k]] in
        ys (K, N, 4) and idxs (K, N); y and idx end at the last one."""
        for i in range(y.shape[0]):
            tri = tr[i] if law == 1 else tr[0]
            lat, lon, h, psi, k_wp = y[i, 0], y[i, 1], y[i, 2], y[i, 3], idx[i]
            j = np.int64(0)  # not a literal 0: _rk4_steps_nb would compile again for Literal[int](0)
            for k in range(ends.size):
                lat, lon, h, psi, k_wp = _rk4_steps_nb(law, params[i], tri, wp[i], cnt[i], sw, ts, j, ends[k],
                                                       lat, lon, h, psi, k_wp, a, e2)
                j = ends[k]
                ys[k, i, 0], ys[k, i, 1], ys[k, i, 2], ys[k, i, 3] = lat, lon, h, psi
                idxs[k, i] = k_wp
            y[i, 0], y[i, 1], y[i, 2], y[i, 3] = lat, lon, h, psi
            idx[i] = k_wp
