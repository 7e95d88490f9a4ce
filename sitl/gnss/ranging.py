"""Light-time geometry between GNSS satellites and receivers (ECEF, SI units).

The signal received at time t_rx by a receiver at r(t_rx) left the satellite at
t_rx - tau.  Both ends are expressed in the Earth-fixed frame *at reception*: the
satellite's ECEF position at emission, p(t_rx - tau), is rotated by the angle the
Earth turns during the flight (the Sagnac / Earth-rotation correction):

    s = R3(w_e tau) p(t_rx - tau),   R3(a) = [[cos a, sin a, 0], [-sin a, cos a, 0], [0, 0, 1]],
    rho = |s - r|,   tau = rho / c                                   (light-time equation)

(IS-GPS-200 sec. 20.3.3.4.3.3.2, Earth rotation correction; Misra & Enge, *Global
Positioning System*, 2nd ed., sec. 5.1; Ashby 2003, Living Rev. Relativ. 6:1).
The fixed point is found by iteration; each step contracts the error by
|d rho / d tau| / c < 2e-5.

Range rate.  Differentiating s(t) = R3(w tau(t)) p(t - tau(t)) with
d R3(a)/da x = -z x (R3(a) x):

    ds/dt = R v - tau' (R v + w z x s) = R v - tau' w_in,

where v = dp/dt_e is the satellite's ECEF (rotating-frame) velocity at emission and
w_in = R v + w z x s its inertial velocity expressed in the reception frame.  With
rho' = u.(ds/dt - r'), u = (s - r)/rho and tau' = rho'/c this is linear in rho':

    rho' = u.(R v - r') / (1 + u.w_in / c)                        (closed form)

and then ds/dt = R v - (rho'/c) w_in, so that rho' = u.(ds/dt - r') exactly.

Speed.  Satellite states at the per-receiver emission times are not propagated one
by one: for each distinct reception time (or on a 1 s grid when there are many),
the exact ephemeris state (position and velocity) is computed at two epochs that
bracket the emission window, and the emission state is the cubic Hermite
interpolant between them.  Its interpolation error is at most |d^4p/dt^4| H^4 / 384
with |d^4 p/dt^4| < 1e-7 m/s^4 for GNSS orbits in the rotating frame: < 1e-13 m for
the 0.12 s bracket and < 3e-10 m on the 1 s grid.  Float64 rounding of the node
states, amplified in forming the coefficients, leaves differences from direct
evaluation of ~1e-7 m and ~1e-7 m/s, far below the mm and mm/s level; the range rate
is the exact derivative of the interpolated range.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from filters.params import ParamError
from sitl.constants import C_M_S, ellipsoid
from sitl.gnss.orbits import Constellation, _propagate

__all__ = ["Geometry", "finite_vec3", "light_time_geometry", "sat_state_at_reception_frame", "LIGHT_TIME_TOL_S"]

#: The light-time iteration stops when tau changes by less than this.  The returned
#: satellite position is the one evaluated at the previous iterate, within 1e-12 s of
#: the returned tau_s = range_m / c (< 4e-9 m of satellite motion), and both are
#: within ~2e-5 * 1e-12 s (the contraction factor) of the exact fixed point.
LIGHT_TIME_TOL_S = 1e-12
_MAX_ITER = 12
_BRACKET_S = 0.12  # emission window [t_rx - 0.12 s, t_rx]: tau is 64..90 ms above the
# horizon and < 110 ms even through the Earth (range < a + R_earth)
_GRID_S = 1.0  # node spacing when reception times are too many to bracket one by one


@dataclass(frozen=True, eq=False)
class Geometry:
    """Receiver-satellite light-time geometry, batch shape (...) and S satellites.

    range_m : (..., S) |s - r|: satellite at emission (rotated into the reception
        ECEF frame) to receiver at reception.  Equal to C_M_S * tau_s.
    range_rate_m_s : (..., S) exact d(range_m)/d(t_rx), positive when receding.
    tau_s : (..., S) signal transit time, range_m / C_M_S.
    sat_pos_ecef_m : (..., S, 3) s = R3(w_e tau) p(t_rx - tau): the satellite at
        emission in the ECEF frame of the reception time.
    sat_vel_ecef_m_s : (..., S, 3) ds/dt_rx, the total derivative of sat_pos_ecef_m
        with respect to the reception time along the light-time solution,
        R3(w_e tau) v(t_rx - tau) - (range_rate/c) (R3 v + w_e z x s), v being the
        rotating-frame ECEF velocity at emission.  With it the range rate is exactly
        ``los_unit . (sat_vel_ecef_m_s - rx_vel_ecef_m_s)``.  The first term alone is
        what :func:`sat_state_at_reception_frame` returns with tau_rate_s_s = 0; the
        second is ~1e-2 m/s.
    los_unit : (..., S, 3) unit vectors receiver -> satellite, (s - r) / range.
    """

    range_m: np.ndarray
    range_rate_m_s: np.ndarray
    tau_s: np.ndarray
    sat_pos_ecef_m: np.ndarray
    sat_vel_ecef_m_s: np.ndarray
    los_unit: np.ndarray


def _check_constellation(constellation) -> Constellation:
    if not isinstance(constellation, Constellation):
        raise ValueError(f"constellation: expected a Constellation, got {type(constellation).__name__}")
    return constellation


def finite_vec3(key: str, value) -> np.ndarray:
    """A check (key, value) -> value of the filters.params kind for a function argument that is
    a batch of positions or velocities: a finite (..., 3) float array, np.asarray of ``value``
    (no copy), else ParamError naming ``key``. (The core's array() fixes the number of axes;
    these arguments have any.)"""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ParamError(key, f"expected a finite (..., 3) array, got a {type(value).__name__}") from None
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise ParamError(key, f"expected a finite (..., 3) array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ParamError(key, "expected a finite (..., 3) array, got non-finite values")
    return arr


def _times(name: str, value) -> np.ndarray:
    t = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name}: times must be finite")
    return t


def _omega(ell) -> float:
    try:
        return ellipsoid(ell).omega_rad_s
    except ValueError as exc:
        raise ValueError(f"ell: {exc}") from None


def _cos_sin(theta: np.ndarray):
    """cos and sin of the Earth-rotation angle (new arrays), see :func:`_rotation`."""
    ct, st = np.empty_like(theta), np.empty_like(theta)
    _rotation(theta, ct, st)
    return ct, st


def _rotated_state(x, y, z, vx, vy, vz, tau, we, tau_rate):
    """s = R3(w tau) p and ds/dt_rx = R3 v - tau' (R3 v + w z x s), component-wise."""
    ct, st = _cos_sin(we * tau)
    sx, sy = ct * x + st * y, ct * y - st * x
    rvx, rvy = ct * vx + st * vy, ct * vy - st * vx
    wx, wy = rvx - we * sy, rvy + we * sx  # inertial velocity, z x s = (-sy, sx, 0)
    return (sx, sy, z), (rvx - tau_rate * wx, rvy - tau_rate * wy, vz - tau_rate * vz), (wx, wy, vz)


def sat_state_at_reception_frame(t_rx_gps_s, tau_s, constellation: Constellation,
                                 tau_rate_s_s=0.0, ell=None) -> tuple[np.ndarray, np.ndarray]:
    """Satellite positions/velocities for a given transit time, in the reception frame.

    For an estimator that knows t_rx and a transit time tau (e.g. its measured
    pseudorange / c, corrected for its clock) this returns the same quantities as
    :func:`light_time_geometry` without touching the true receiver state
    (direct ephemeris evaluation at t_rx - tau, no interpolation):

        s = R3(w_e tau) p(t_rx - tau),
        ds/dt_rx = R3(w_e tau) v(t_rx - tau) - tau' (R3 v + w_e z x s),

    p, v the ECEF (rotating-frame) ephemeris state at emission and tau' = d tau/d t_rx
    (``tau_rate_s_s``; 0 gives the velocity at a fixed transit time, R3 v; pass
    range_rate / c for the exact derivative of light_time_geometry).

    Parameters
    ----------
    t_rx_gps_s : (...) reception GPS time, broadcast against tau_s.shape[:-1].
    tau_s : (..., S) transit time per satellite (last axis = constellation order).
    constellation : Constellation with S satellites.
    tau_rate_s_s : scalar or (..., S), d tau / d t_rx (dimensionless).
    ell : Ellipsoid or name whose rotation rate turns the frame during the flight
        (default WGS-84).

    Returns
    -------
    sat_pos_ecef_m, sat_vel_ecef_m_s : (..., S, 3).
    """
    c = _check_constellation(constellation)
    we = _omega(ell)
    tau = _times("tau_s", tau_s)
    S = len(c)
    if tau.ndim < 1 or tau.shape[-1] != S:
        raise ValueError(f"tau_s: expected shape (..., {S}), got {tau.shape}")
    t = _times("t_rx_gps_s", t_rx_gps_s)
    try:
        batch = np.broadcast_shapes(t.shape, tau.shape[:-1])
    except ValueError:
        raise ValueError(f"t_rx_gps_s: shape {t.shape} does not broadcast with tau_s batch {tau.shape[:-1]}") from None
    shape = batch + (S,)
    rate = _times("tau_rate_s_s", tau_rate_s_s)
    try:
        np.broadcast_shapes(rate.shape, shape)
    except ValueError:
        raise ValueError(f"tau_rate_s_s: shape {rate.shape} does not broadcast with {shape}") from None
    # Satellite-major (S, F) evaluation; (t - toa) first: exact for nearby float64
    # values, so tau keeps full precision.
    tau_sf = np.broadcast_to(tau, shape).reshape(-1, S).T
    rate_sf = np.broadcast_to(rate, shape).reshape(-1, S).T
    t_f = np.broadcast_to(t, batch).reshape(1, -1)
    x, y, z, vx, vy, vz = _propagate(c, (t_f - c.toa_gps_s[:, None]) - tau_sf, want_vel=True, sat_major=True)
    s, ds, _ = _rotated_state(x, y, z, vx, vy, vz, tau_sf, we, rate_sf)
    return _to_batch_vec(s, batch, S), _to_batch_vec(ds, batch, S)


def _to_batch_vec(comps, batch, S) -> np.ndarray:
    """3 components of shape (S, F) (or broadcastable) -> contiguous (*batch, S, 3)."""
    out = np.empty(batch + (S, 3))
    view = out.reshape(-1, S, 3)
    F = view.shape[0]
    comps = [np.broadcast_to(q, (S, F)) for q in comps]
    if F >= S:  # row-wise copies are the fastest transposition for long rows
        for j in range(S):
            for k in range(3):
                view[:, j, k] = comps[k][j]
    else:
        for k in range(3):
            view[:, :, k] = comps[k].T
    return out


def _to_batch(a, batch, S) -> np.ndarray:
    """(S, F) -> contiguous (*batch, S)."""
    out = np.empty(batch + (S,))
    view = out.reshape(-1, S)
    a = np.broadcast_to(a, (S, view.shape[0]))
    if view.shape[0] >= S:
        for j in range(S):
            view[:, j] = a[j]
    else:
        view[...] = a.T
    return out


def _hermite(c: Constellation, t_f: np.ndarray):
    """Cubic Hermite models of the ECEF ephemeris around the emission times.

    ``t_f`` (F,) are reception times.  Returns (off, coef): off ((F,) or (1,)) is
    t_rx - T_a, the reception instant measured from node a, and coef = 3 tuples
    (p0, v0, c2, c3) of (S, F) or (S, 1) arrays (one tuple per axis) such that the
    satellite state at the emission time t_rx - tau is, with s = off - tau,

        p(s) = p0 + v0 s + c2 s^2 + c3 s^3,   v(s) = v0 + 2 c2 s + 3 c3 s^2,

    matching the exact ephemeris (p0, v0) at T_a and (p1, v1) at T_b = T_a + H:
    A = (p1 - p0 - v0 H)/H^2, B = (v1 - v0)/H, c2 = 3A - B, c3 = (B - 2A)/H.

    Nodes: T_a = t_rx - 0.12 s, T_b = t_rx for each distinct reception time, or, when
    that is cheaper, the 1 s grid segment [T_a, T_a + 1 s] holding t_rx - 0.075 s
    (the segment stays fixed while iterating; the cubic extrapolates smoothly).
    """
    tu, inv = np.unique(t_f, return_inverse=True)
    toa = c.toa_gps_s[:, None]
    seg = np.floor((t_f - 0.075) / _GRID_S)
    useg, sinv = np.unique(seg, return_inverse=True)
    # Node times as t - toa, computed so that no precision is lost (|t| ~ 1e9 s).
    if useg.size < tu.size:
        H = _GRID_S
        tk_a = (useg * _GRID_S)[None, :] - toa
        off = t_f - seg * _GRID_S
        gather = sinv if useg.size > 1 else None
    else:
        H = _BRACKET_S
        tk_a = (tu[None, :] - toa) - H
        off = np.full(1, _BRACKET_S)
        gather = inv if (tu.size > 1 and (tu.size < t_f.size or np.any(np.diff(t_f) <= 0))) else None
    a_state = _propagate(c, tk_a, want_vel=True, sat_major=True)
    b_state = _propagate(c, tk_a + H, want_vel=True, sat_major=True)
    coef = []
    for k in range(3):
        p0, v0, p1, v1 = a_state[k], a_state[3 + k], b_state[k], b_state[3 + k]
        A = (p1 - p0 - v0 * H) * (1.0 / (H * H))
        B = (v1 - v0) * (1.0 / H)
        cf = (p0, v0, 3.0 * A - B, (B - 2.0 * A) * (1.0 / H))
        coef.append(cf if gather is None else tuple(q[:, gather] for q in cf))
    return off, coef


def light_time_geometry(t_rx_gps_s, rx_pos_ecef_m, rx_vel_ecef_m_s, constellation: Constellation,
                        ell=None) -> Geometry:
    """Light-time-corrected ranges, range rates and lines of sight.

    Solves tau = |R3(w_e tau) p(t_rx - tau) - r| / c by fixed-point iteration from
    the instantaneous range (until tau moves by < ``LIGHT_TIME_TOL_S``), then the
    exact range rate in closed form (see the module docstring):

        rho' = u.(R3 v - r') / (1 + u.(R3 v + w_e z x s) / c).

    Parameters
    ----------
    t_rx_gps_s : (...) true reception GPS time.
    rx_pos_ecef_m : (..., 3) receiver ECEF position at t_rx.
    rx_vel_ecef_m_s : (..., 3) receiver ECEF velocity at t_rx (rotating frame).
    constellation : Constellation with S satellites.
    ell : Ellipsoid or name (default WGS-84) whose rotation rate turns the frame
        during the signal flight.  The ephemeris itself uses each system's own
        constants; PZ-90.11 and WGS-84 frames are treated as identical (no datum
        transformation).

    The batch shape (...) is the broadcast of t_rx_gps_s.shape,
    rx_pos_ecef_m.shape[:-1] and rx_vel_ecef_m_s.shape[:-1] (normally t broadcasts
    to the receivers' shape; one receiver at many times also works).

    Returns
    -------
    Geometry with (..., S) and (..., S, 3) arrays.
    """
    c = _check_constellation(constellation)
    we = _omega(ell)
    r = finite_vec3("rx_pos_ecef_m", rx_pos_ecef_m)
    v = finite_vec3("rx_vel_ecef_m_s", rx_vel_ecef_m_s)
    t = _times("t_rx_gps_s", t_rx_gps_s)
    try:
        batch = np.broadcast_shapes(r.shape[:-1], v.shape[:-1])
    except ValueError:
        raise ValueError(f"rx_vel_ecef_m_s: shape {v.shape} does not broadcast with rx_pos_ecef_m {r.shape}") from None
    try:
        batch = np.broadcast_shapes(t.shape, batch)
    except ValueError:
        raise ValueError(f"t_rx_gps_s: shape {t.shape} does not broadcast with the receivers' {batch}") from None
    S = len(c)

    # Satellite-major layout: (S, F) arrays, F = prod(batch) (t may be shared: F_t = 1).
    t_f = t.reshape(1) if t.size == 1 else np.broadcast_to(t, batch).reshape(-1)
    rx, ry, rz = np.broadcast_to(r, batch + (3,)).reshape(-1, 3).T.copy()
    vrx, vry, vrz = np.broadcast_to(v, batch + (3,)).reshape(-1, 3).T.copy()
    off, coef = _hermite(c, t_f)
    F = rx.size
    # All arithmetic below goes into preallocated (S, F) buffers: with numpy's
    # fresh temporaries the allocator's page faults cost more than the arithmetic.
    buf = np.empty((17, S, F))
    s, x, y, z, sx, sy, tmp, rho, tau, tau_new, th, ct, st, vx, vy, vz, aux = buf
    tau[...] = np.sqrt(sum((p0 + off * (v0 + off * (c2 + off * c3)) - rk) ** 2
                           for (p0, v0, c2, c3), rk in zip(coef, (rx, ry, rz)))) * (1.0 / C_M_S)
    # Initial tau from the instantaneous range (s = off, i.e. tau = 0): off by ~1e-6 s.
    for _ in range(_MAX_ITER):
        np.subtract(off, tau, out=s)
        for out, cf in zip((x, y, z), coef):
            _horner(out, s, *cf)
        np.multiply(tau, we, out=th)
        _rotation(th, ct, st)
        np.multiply(ct, x, out=sx)
        np.multiply(st, y, out=tmp)
        sx += tmp
        np.multiply(ct, y, out=sy)
        np.multiply(st, x, out=tmp)
        sy -= tmp
        dx, dy, dz = np.subtract(sx, rx, out=x), np.subtract(sy, ry, out=y), np.subtract(z, rz, out=aux)
        np.multiply(dx, dx, out=rho)
        rho += np.multiply(dy, dy, out=tmp)
        rho += np.multiply(dz, dz, out=tmp)
        np.sqrt(rho, out=rho)
        np.multiply(rho, 1.0 / C_M_S, out=tau_new)
        step = np.abs(np.subtract(tau_new, tau, out=tmp), out=tmp).max(initial=0.0)
        tau, tau_new = tau_new, tau
        if step < LIGHT_TIME_TOL_S:
            break
    else:  # pragma: no cover - needs receivers moving at a sizeable fraction of c
        raise RuntimeError("light-time iteration did not converge")
    sz = z  # rotation about z leaves z alone; x, y, aux now hold dx, dy, dz

    # Velocity at emission (exact derivative of the Hermite model), rotated: R v.
    for out, (_, v0, c2, c3) in zip((vx, vy, vz), coef):
        np.multiply(c3, s, out=out)
        out *= 1.5
        out += c2
        out *= s
        out *= 2.0
        out += v0
    rvx = np.multiply(ct, vx, out=tau_new)
    rvx += np.multiply(st, vy, out=tmp)
    rvy = np.multiply(ct, vy, out=th)
    rvy -= np.multiply(st, vx, out=tmp)
    # Inertial velocity in the reception frame: w = R v + w_e z x s, z x s = (-sy, sx).
    wx = np.multiply(sy, -we, out=vx)
    wx += rvx
    wy = np.multiply(sx, we, out=vy)
    wy += rvy
    inv_rho = np.divide(1.0, rho, out=ct)
    ux, uy, uz = (np.multiply(d, inv_rho, out=d) for d in (dx, dy, dz))
    # rho' = u.(R v - r') / (1 + u.w / c)
    num = np.multiply(ux, rvx - vrx, out=st)
    num += np.multiply(uy, rvy - vry, out=tmp)
    num += np.multiply(uz, vz - vrz, out=tmp)
    den = np.multiply(ux, wx, out=s)
    den += np.multiply(uy, wy, out=tmp)
    den += np.multiply(uz, vz, out=tmp)
    den *= 1.0 / C_M_S
    den += 1.0
    rho_dot = np.divide(num, den, out=num)
    tau_rate = np.multiply(rho_dot, 1.0 / C_M_S, out=den)
    # ds/dt_rx = R v - tau' w
    svx = np.subtract(rvx, np.multiply(tau_rate, wx, out=tmp), out=rvx)
    svy = np.subtract(rvy, np.multiply(tau_rate, wy, out=tmp), out=rvy)
    svz = np.subtract(vz, np.multiply(tau_rate, vz, out=tmp), out=wx)

    return Geometry(
        range_m=_to_batch(rho, batch, S),
        range_rate_m_s=_to_batch(rho_dot, batch, S),
        tau_s=_to_batch(tau, batch, S),
        sat_pos_ecef_m=_to_batch_vec((sx, sy, sz), batch, S),
        sat_vel_ecef_m_s=_to_batch_vec((svx, svy, svz), batch, S),
        los_unit=_to_batch_vec((ux, uy, uz), batch, S),
    )


def _horner(out, s, p0, v0, c2, c3):
    """out = p0 + s (v0 + s (c2 + s c3)), in place."""
    np.multiply(c3, s, out=out)
    out += c2
    out *= s
    out += v0
    out *= s
    out += p0


def _rotation(theta, ct, st):
    """cos and sin of the Earth-rotation angle into ct, st.  For |theta| < 1e-4 (tau
    below 1.3 s) the series 1 - theta^2/2 and theta (1 - theta^2/6) are exact in
    float64 (next terms < 1e-17 relative); np.cos/np.sin otherwise."""
    if np.max(np.abs(theta), initial=0.0) < 1e-4:
        np.multiply(theta, theta, out=ct)
        np.multiply(ct, -1.0 / 6.0, out=st)
        st += 1.0
        st *= theta
        ct *= -0.5
        ct += 1.0
    else:
        np.cos(theta, out=ct)
        np.sin(theta, out=st)
